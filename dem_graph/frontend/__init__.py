"""The visual front end: patch extraction and active-search tracking of guided points."""
