"""A heap of fragments: screening the pairs, the spanning forest, pose-graph refinement, the
outputs, engines, grouping a mixed heap by object, and scoring against a known answer."""
