"""``python -m gausslite_services.fusion_server [--host H] [--port P] [--data-dir D] [--port-file F] ...``."""

import sys

from gausslite_services.fusion_server.server import main

sys.exit(main())
