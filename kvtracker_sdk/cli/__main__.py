"""``python -m kvtracker_sdk.cli``: the ``kvtracker`` command without the console script."""

from kvtracker_sdk.cli.app import main

main()
