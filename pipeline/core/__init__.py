"""The kernel every stage builds on; it imports no stage.

errors (one exception hierarchy), artifacts (atomic writes, crash-safe output directories), manifest (provenance,
hashes), config (typed configs, YAML profiles, dotted overrides), stage (run a stage body into an output directory),
layout (the data-dir tree as path templates), keys (observation and dataset feature names), timing.
"""
