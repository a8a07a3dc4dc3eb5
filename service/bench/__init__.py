"""slamtka.bench: tooling, not part of the product."""
