"""Scenario schema, diagram builders, runner, benchmarks and the maglev CLI."""
