"""Loop closure before plane adjustment: local maps, place descriptors, verified closures, pose graph.

`close_loops(points, T_world_scan, config.advanced.loops, config.loops.min_separation_m)` returns a
`LoopResult` with loop-closed T_world_scan and the record of every candidate (see `closure` for the
method).
"""

from pa_cli.loops.closure import Candidate, LoopResult, close_loops

__all__ = ["Candidate", "LoopResult", "close_loops"]
