"""The command-line verbs, one module each, on top of every stage package (see docs/architecture.md)."""
