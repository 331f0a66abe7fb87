"""Datasets in and out: robomimic-layout HDF5 (``hdf5``: load_dataset, write_dataset, DemoWriter), LeRobotDataset
v3.0 (``lerobot``), raw simulator states rendered to image observations (``render_dataset``) and delta
actions replayed to absolute ones (``convert_abs_actions``).
"""
