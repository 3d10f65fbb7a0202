"""`python -m jaxfoam ...`: the same command line as `jaxfoam ...`."""
import sys

from .cli import main

sys.exit(main())
