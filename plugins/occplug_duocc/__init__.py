"""occplug-duocc: DuOcc (stream- and query-guided feature aggregation), work in progress.

Registered (``plugin.py``): the ``duocc_stream`` scene (3D-FPN + StreamAgg, stateful), the ``duocc_stacking``
multi-frame baseline scene, the ``duocc_decoder`` head and the ``duocc_occupied`` / ``duocc_forecast``
supervision sources; configs ``duocc/single_frame`` (Tab. 4 A), ``duocc/stream_agg`` (Tab. 4 B), the Tab. 5 rows
and ``duocc/stacking``. Building blocks not yet registered: Hungarian matching (``matching``) and dynamic query
aggregation (``dqa``) for QueryAgg.
"""
