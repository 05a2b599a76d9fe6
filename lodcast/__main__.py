"""`python -m lodcast ...`: the `lodcast` command."""
from lodcast.service.cli import main

raise SystemExit(main())
