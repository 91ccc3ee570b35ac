"""Live intake (``live_intake``): an adapter over a tracker's ``push_frame`` for a live camera:
frames handed over without waiting, tracked on a worker thread with the newest frame winning,
results and errors delivered through the tracker's callbacks (``on_result``, ``on_frame_error``).
"""
