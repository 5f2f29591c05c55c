"""Small real stages for the engine's tests: they read their inputs, write outputs, count runs."""
