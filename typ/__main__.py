import sys

from typ.cli import main

sys.exit(main())
