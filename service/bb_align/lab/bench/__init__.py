"""``bb-align bench``: the engine timed stage by stage against a straightforward in-benchmark baseline, on a
fixed seeded workload, plus the service's throughput over Zenoh. See docs/performance.md."""
