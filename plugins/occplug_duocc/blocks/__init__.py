"""DuOcc's building blocks, used by its components (``scene``, ``heads``, ``supervision``): ``fpn3d`` (the 3D-FPN),
``stream_agg`` (RefineNet, the stream fusion and its losses), ``queryagg`` (I2Q, V2Q and DQA wired together),
``dqa``, ``detector`` (the Sparse4D-style image-to-query detector), ``image_aggregation`` (its deformable
multi-camera, multi-level image sampling), ``boxes`` (the encoded box), ``detection_loss``, ``v2q``
(``VoxelToQuery``), ``denoising`` and ``matching``."""
