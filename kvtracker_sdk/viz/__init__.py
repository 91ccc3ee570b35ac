"""Layer 6: optional visualisation (``rerun_sink.RerunSink``; rerun loads only when used)."""
