"""``python -m gausslite_services.agent [serve-options]`` = ``gausslite serve agent [serve-options]``."""

import sys

from gausslite.cli import run_as_program

run_as_program(["serve", "agent", *sys.argv[1:]])
