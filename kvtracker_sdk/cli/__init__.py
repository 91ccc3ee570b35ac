"""Layer 6: the ``kvtracker`` command line (typer). The only place in the SDK that configures
logging and draws progress bars; ``app.py`` assembles one module per command group."""
