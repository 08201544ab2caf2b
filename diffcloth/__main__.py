"""`python -m diffcloth ...` is the `diffcloth` command."""

from diffcloth.cli import main

raise SystemExit(main())
