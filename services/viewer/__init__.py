"""Live viewer feed: follows a fusion server over gRPC and drives :class:`gausslite.viewer.app.MapViewer`."""
