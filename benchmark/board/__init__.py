"""``skidbench compare``: which runs a board is made of, its rows and tables."""
