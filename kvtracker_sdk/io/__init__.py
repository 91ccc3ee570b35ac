"""Reading and writing what the tracker keeps and meets, one folder per concern.

- ``map_file/``: the ``.kvmap`` map file: its header, tensor schema, codec, reader and writer.
- ``sources/``: where frames come from: image folders, videos, datasets, cameras, depth images,
  camera calibration files.
- ``exports/``: what other tools read: PLY point clouds, COLMAP and nerfstudio datasets, ROS 2 bags.
- ``files/``: single files shared by the others: atomic writes, capped reads of user-named files,
  TUM/KITTI trajectories, the tuner's cache.

Imports point one way (``pyproject.toml``'s import contracts): ``exports`` may use
``map_file`` and ``sources``, which do not use each other; all three may use ``files``.
"""
