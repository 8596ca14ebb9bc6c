"""``gausslite view``: show a Gaussian map in the browser (viser), or follow a fusion server live.

    gausslite view MAP.ply [--port 8080] [--color rgb|kappa|roi]     # also .splat / .spz
    gausslite view --fusion HOST:PORT [--poll 1.0] [--token T]       # new fused versions appear live
    gausslite view --fusion HOST:PORT --tls-ca ca.pem --tls-client-cert viewer.pem --tls-client-key viewer.key

Open the printed URL (``http://127.0.0.1:8080/``). A map file is loaded after the URL is printed: a
page opened meanwhile shows the loading progress (progress bar and notification), as does the console.
The GUI panel switches the colouring (RGB, κ, ROI), shows only the ROI (active) Gaussians, toggles
keyframe trajectories and frusta and, with ``--fusion``, lists agents, shares, bytes and versions.
``--host 0.0.0.0`` serves the page to other machines. The fusion server's credentials take the options of
every client command (``--tls-ca``, ``--tls-client-cert``, ``--tls-client-key`` for TLS and mutual TLS,
``--token`` / ``--token-file``) with the agents' environment fallbacks (``docs/security.md``):
``GAUSSLITE_TLS_CA``, ``GAUSSLITE_TLS_CLIENT_CERT`` / ``GAUSSLITE_TLS_CLIENT_KEY``, a per-agent token
``GAUSSLITE_FUSION_TOKEN`` / ``GAUSSLITE_FUSION_TOKEN_FILE``, else the fleet token ``GAUSSLITE_TOKEN``. Further
environment fallbacks: ``GAUSSLITE_VIEW_PORT``, ``GAUSSLITE_FUSION_ADDR``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

from gausslite.core.environment import EnvironmentSettings
# grpc-free: the command line registers the options without loading the services
from gausslite_services.common.cli_options import add_client_credential_arguments, client_credentials_from_args


def register(subparsers) -> None:
    """Add the ``view`` subcommand to ``subparsers``."""
    # lazy: the command line starts without loading the services or gRPC
    from gausslite.viewer.app import UP_AXES
    from gausslite.viewer.splats import COLOR_MODES

    p = subparsers.add_parser("view", help="show a map (or a live fusion server) in the browser",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("map", nargs="?", default=None, help="map file (.ply, .splat, .spz)")
    p.add_argument("--fusion", default=None, metavar="HOST:PORT",
                   help="follow this fusion server live instead of a file (env GAUSSLITE_FUSION_ADDR)")
    p.add_argument("--host", default="127.0.0.1", help="bind address of the web page (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=None, help="web page port (env GAUSSLITE_VIEW_PORT, default 8080)")
    p.add_argument("--color", choices=COLOR_MODES, default="rgb", help="initial colouring (default rgb)")
    p.add_argument("--roi-only", action="store_true", help="start showing only ROI (active) Gaussians")
    p.add_argument("--up", default="auto", choices=["auto", *UP_AXES],
                   help="world up axis of the initial camera (auto: from keyframes, else +z)")
    p.add_argument("--poll", type=float, default=1.0, help="seconds between fusion-server polls (default 1)")
    p.add_argument("--timeout", type=float, default=None,
                   help="stop after this many seconds (default: run until Ctrl-C)")
    add_client_credential_arguments(p.add_argument_group("fusion server credentials (with --fusion)"),
                                    server="the fusion server")
    p.set_defaults(func=_handle)


def _handle(args: argparse.Namespace) -> int:
    try:
        variables = EnvironmentSettings.read()
    except ValueError as e:
        print(f"gausslite view: error: {e}", file=sys.stderr)
        return 2
    fusion = args.fusion or (None if args.map else variables.fusion_addr)
    if bool(args.map) == bool(fusion):
        print("gausslite view: error: give either a map file or --fusion HOST:PORT", file=sys.stderr)
        return 2
    try:
        if args.map:  # a missing or unsupported file fails before a page is served
            # lazy: the command line starts without loading the services or gRPC
            from gausslite.viewer.export import format_of

            format_of(args.map)
            if not os.path.isfile(args.map):
                raise FileNotFoundError(f"map file not found: {args.map}")
        port = next(p for p in (args.port, variables.view_port, 8080) if p is not None)
        if not args.poll > 0:
            raise ValueError(f"--poll must be > 0, got {args.poll}")
        # lazy: the command line starts without loading the services or gRPC
        from gausslite.viewer.app import MapViewer

        viewer = MapViewer(args.host, port, up=args.up)
    except (ValueError, OSError) as e:
        print(f"gausslite view: error: {e}", file=sys.stderr)
        return 2
    viewer.color_mode.value = args.color
    viewer.roi_only.value = bool(args.roi_only)
    feed = client = None
    try:
        if args.map:
            # lazy: the command line starts without loading the services or gRPC
            from gausslite.viewer.export import load_map

            # The page is served from here on: print its URL first, then read and convert the map, so
            # a browser opened now sees the progress (panel text, progress bar and a notification).
            label, nbytes = os.path.basename(args.map), os.path.getsize(args.map)
            print(f"serving {viewer.url} (loading {args.map}, {nbytes / 1e6:,.1f} MB; open the page to watch "
                  "the progress)", flush=True)
            viewer.show_reading(label, nbytes)
            try:
                g = load_map(args.map)
                viewer.set_map(g, label=label)
            except (OSError, ValueError) as e:
                print(f"gausslite view: error: {e}", file=sys.stderr)
                return 2
            except KeyboardInterrupt:
                return 130
            print(f"showing {args.map} ({len(g):,} Gaussians) at {viewer.url}", flush=True)
        else:
            # lazy: the command line starts without loading the services or gRPC
            from gausslite_services.fusion_server.client import FusionClient
            from gausslite_services.viewer.feed import FusionFeed

            try:
                creds = client_credentials_from_args(args)
            except (ValueError, OSError) as e:
                print(f"gausslite view: error: {e}", file=sys.stderr)
                return 2
            client = FusionClient(fusion, **creds)
            feed = FusionFeed(viewer, client, poll_s=args.poll).start()
            print(f"following fusion server {fusion} at {viewer.url}", flush=True)
        deadline = None if args.timeout is None else time.monotonic() + args.timeout
        try:
            while deadline is None or time.monotonic() < deadline:
                time.sleep(0.2)
        except KeyboardInterrupt:
            pass
        return 0
    finally:
        if feed is not None:
            feed.stop()
        if client is not None:
            client.close()
        viewer.stop()
