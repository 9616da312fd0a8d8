"""Dataset-level drivers: run a stage over every frame of a dataset into a run folder.

* :mod:`radarpc.pipelines.pointclouds`: a RADIal root -> a Parquet point store;
* :mod:`radarpc.pipelines.sparse_rd`: a RADIal root -> a sparse-RD root (the same layout);
* :mod:`radarpc.pipelines.oscfar`: a ColoRadar root -> OS-CFAR prediction folders;
* :mod:`radarpc.pipelines.radial_pcl`: a point store -> its RADIal root's ``radar_PCL/`` files.

Each one owns its output through :mod:`radarpc.runs` (lock, key check, resume) and spreads work
through :mod:`radarpc.distributed` (torchrun ranks, local workers).
"""
