"""Command runners: each `pressurepose` subcommand's config, `run_*`, report and figure writers.
Library modules below return typed results; only commands (and viz) write reports."""
