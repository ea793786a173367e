"""The VAD-GS event before issue 21 (commit 274c932), frozen as the reference of bench_vad_event."""
