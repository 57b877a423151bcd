"""The dataset formats the readers know (``open_dataset``'s ``format``): the one tuple every ``--format`` flag reads."""

FORMATS = ("deeploc", "7scenes")
