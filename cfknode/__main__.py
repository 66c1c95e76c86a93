import sys

from cfknode.app.cli import main

sys.exit(main())
