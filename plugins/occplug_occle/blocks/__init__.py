"""OccLE's building blocks, used by its components: ``geometry_branch`` (the cross-plane branch and the LiDAR voxel
encoder), ``mamba`` and ``selective_scan`` (Dual Mamba), ``serialization`` (Hilbert order), ``projection`` (the
image-plane projection head) and ``losses``. Its UNets and deformable attention are the core's, :mod:`occplug.nn`."""
