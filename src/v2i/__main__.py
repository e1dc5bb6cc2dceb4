import sys

from v2i.cli import main

sys.exit(main())
