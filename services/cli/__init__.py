"""The ``gausslite`` subcommands that run or call the gRPC services (``sim``, ``serve``, ``health``, ``tokens``,
``view``). The library's CLI (:mod:`gausslite.cli`) finds them through the ``gausslite.commands`` entry point, so
the library itself never imports the services."""
