import sys

from aqfg.cli import main

sys.exit(main())
