"""The tracker's side of map files (``tracker_maps``): what is saved with a map, and what a loaded
map runs under.
"""
