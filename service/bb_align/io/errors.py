"""The error a bad input file raises. Kept free of imports so the CLI can catch it without loading numpy."""


class InputFileError(ValueError):
    """A cloud or box file that is not what it should be. str(): '<path>: <problem> (<what is allowed>)'."""
