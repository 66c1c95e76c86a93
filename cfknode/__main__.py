import sys

from cfknode.cli import main

sys.exit(main())
