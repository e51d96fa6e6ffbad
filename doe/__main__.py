import sys

from doe.cli import main

sys.exit(main())
