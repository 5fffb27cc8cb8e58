"""physicsrl."""
