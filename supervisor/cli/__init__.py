"""Command line: ``supervisor run | check | schema | bench``."""
