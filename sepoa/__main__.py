"""`python -m sepoa ...`: the `sepoa` command without its script (how `sepoa up` and
`sepoa experiment run` start their workers, with this interpreter)."""

import sys

from sepoa.cli import main

sys.exit(main())
