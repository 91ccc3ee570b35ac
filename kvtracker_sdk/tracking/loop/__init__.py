"""The per-frame loop: one tracking step per frame (``frame_loop``), the tracking state table that
decides the next state (``states``, drawn by ``state_diagram``) and the events a step reports
(``reporting``).
"""
