import sys

from fabkit.cli import entry

sys.exit(entry())
