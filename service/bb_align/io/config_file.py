"""An engine configuration saved as JSON or YAML (``bb-align config --dump``), read back."""

from __future__ import annotations

from pathlib import Path

from pydantic import ValidationError

from bb_align.engine.config import AlignConfig


def load_align_config(path: str | Path | None) -> AlignConfig:
    """An AlignConfig from a JSON or YAML file (defaults for what it leaves out); the defaults without one.
    Raises ValueError naming the file."""
    if path is None:
        return AlignConfig()
    path = Path(path)
    try:
        if path.suffix.lower() in (".yaml", ".yml"):
            import yaml

            return AlignConfig.model_validate(yaml.safe_load(path.read_text()) or {})
        return AlignConfig.model_validate_json(path.read_text())
    except (ValidationError, ValueError) as e:
        raise ValueError(f"{path}: {e}") from None
