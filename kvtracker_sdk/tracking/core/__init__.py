"""The vocabulary every other part of tracking shares: frame validation and model-input
preparation (``frame_input``), per-frame intrinsics (``intrinsics``), confidence (``quality``),
world-frame continuity across rebuilds (``gauge``) and the events the tracker emits (``events``).

Nothing here knows about maps, object mode or the frame loop.
"""
