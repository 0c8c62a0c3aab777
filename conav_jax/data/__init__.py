"""The benchmark's data, generated offline and deterministically from a seed.

categories (51 object categories) + activities (the causal activity graph) -> scene (the JSON
scene format and its validating loader) / scenegen (procedural apartments) -> episodes (motion,
robot starts and geodesic fields as array shards, written atomically by arrayio, listed in a
manifest) <- presets (named dataset sizes). `activity_graph.json` is the shipped graph.
"""
