"""Pictures for people: previews, maps and plots (matplotlib, Agg backend, files only)."""
