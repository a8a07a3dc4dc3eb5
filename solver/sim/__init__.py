"""slamtka.sim: tooling, not part of the product."""
