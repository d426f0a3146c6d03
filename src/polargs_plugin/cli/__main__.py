import sys

from polargs_plugin.cli import main

sys.exit(main())
