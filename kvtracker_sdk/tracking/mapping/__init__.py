"""The keyframe map and its rebuilds: which frames become keyframes (``keyframes``), the rebuild
cycle and its bookkeeping (``map_keeper``), building and inserting into a map (``map_builder``,
``map_insertion``), the background worker (``mapper``) and what a failed rebuild means
(``failures``).
"""
