"""``python -m gausslite_services.agent [serve-options]`` = ``gausslite serve agent [serve-options]``."""

import sys

from gausslite.cli import main

sys.exit(main(["serve", "agent", *sys.argv[1:]]))
