"""An engine configuration saved as JSON or YAML (``bb-align config --dump``), read back."""

from __future__ import annotations

from pathlib import Path

from pydantic import ValidationError

from bb_align.engine.config import AlignConfig, describe_errors


def load_align_config(path: str | Path | None) -> AlignConfig:
    """An AlignConfig from a JSON or YAML file (defaults for what it leaves out); the defaults without one.
    Raises ValueError naming the file."""
    if path is None:
        return AlignConfig()
    path = Path(path)
    try:
        if path.suffix.lower() in (".yaml", ".yml"):
            import yaml

            try:
                data = yaml.safe_load(path.read_text()) or {}
            except yaml.YAMLError as e:
                raise ValueError(f"not valid YAML ({' '.join(str(e).split())})") from None
            return AlignConfig.model_validate(data)
        return AlignConfig.model_validate_json(path.read_text())
    except ValidationError as e:
        raise ValueError(f"{path}: {describe_errors(e, AlignConfig)}") from None
    except ValueError as e:  # not JSON / YAML at all
        raise ValueError(f"{path}: {str(e).splitlines()[0]}") from None
