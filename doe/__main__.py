import sys

from doe.infra.cli import main

sys.exit(main())
