"""Live intake: frames from a capture thread, tracked on a worker thread with the newest frame
winning (``live_intake``), results and errors handed to callbacks.
"""
