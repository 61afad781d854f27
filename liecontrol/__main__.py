import sys

from liecontrol.cli import main

sys.exit(main())
