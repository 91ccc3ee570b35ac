"""The map's world frame: gravity alignment and moving a map into another frame
(``world_alignment``), metric scale fitted from depth (``metric_scale``) and the checks on depth
images that come with frames (``depth_input``).
"""
