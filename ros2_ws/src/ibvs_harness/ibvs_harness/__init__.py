"""The experiment harness: scenario runs, campaigns, reports, plots, bags, feature-level loop."""
