"""``python -m gausslite_services.fusion_server [--host H] [--port P] [--data-dir D] [--port-file F] ...``."""

from gausslite.cli import run_as_program
from gausslite_services.fusion_server.server import main

run_as_program(program=main)
