"""The errors the CLI turns into one line and exit code 2. Kept free of imports so the CLI can catch them without
loading numpy."""


class InputFileError(ValueError):
    """A cloud or box file that is not what it should be. str(): '<path>: <problem> (<what is allowed>)'."""


class MissingExtraError(ImportError):
    """An optional dependency is not installed. str() names the extra that brings it, e.g. bb-align[lab]."""

    def __init__(self, package: str, extra: str, needed_for: str):
        super().__init__(f"{needed_for} needs {package}, which is not installed: pip install 'bb-align[{extra}]'")
