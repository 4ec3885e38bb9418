import sys

from vtube_fleet.cli import main

sys.exit(main())
