"""The map's world frame: gravity alignment and moving a map into another frame
(``world_alignment``) and metric scale fitted from the keyframes' sensor depth (``metric_scale``;
a depth image is checked with its frame in ``core/frame_input``).
"""
