"""``python -m undream.cli``: the same as the ``undream`` command."""
from undream.cli import main

main()
