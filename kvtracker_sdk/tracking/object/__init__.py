"""Object mode: where the object is in each frame (``object_region``, with an optional
``segmenter``), and the object model fused from the keyframes' points (``object_model``, separated
from its support by ``object_separation``).
"""
