"""GaussLite: task-conditioned 3D Gaussian Splatting mapping for robot teams.

The core library. It knows nothing of gRPC: the services in ``services/`` are thin servers over it.
"""

__version__ = "0.1.0"
