"""Single files shared by the rest of ``io/`` and the SDK: atomic writes (``atomic``), capped
whole-file reads of paths a user names (``regular_file``), TUM/KITTI trajectories
(``trajectory``), and the tuner's per-machine cache (``tune_cache``)."""
