"""The compare report: its figures and its Markdown text."""
