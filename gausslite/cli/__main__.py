from gausslite.cli import main
import sys
sys.exit(main())
