"""occplug-duocc: DuOcc (stream- and query-guided feature aggregation), work in progress.

The plugin registers no components yet. Its building blocks are plain ``nn.Module`` s and functions
with their own tests (``tests/test_duocc_blocks.py``): stream aggregation with RefineNet
(``stream_agg``), Hungarian matching for the detection loss (``matching``) and dynamic query
aggregation with its query selection (``dqa``).
"""
