"""The vocabulary every other part of tracking shares: the checks on what is pushed with a frame
(``frame_input``) and its preparation for the model (``model_input``), per-frame intrinsics
(``intrinsics``), confidence (``quality``), world-frame continuity across rebuilds (``gauge``) and
the events the tracker emits (``events``).

Nothing here knows about maps, object mode or the frame loop.
"""
