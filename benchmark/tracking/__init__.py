"""MLflow: the store and its runs, their tags, bookkeeping, logged models and UI links."""
