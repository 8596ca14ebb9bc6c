"""``python -m bench.realtime``: the real-time benchmark's command line (:func:`bench.realtime.cli.main`)."""

import sys

from bench.realtime.cli import main

if __name__ == "__main__":
    sys.exit(main(prog="python -m bench.realtime"))
