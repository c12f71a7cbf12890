"""Command-line tools of `neurncd` that pick data sources for the core (outside the core)."""
