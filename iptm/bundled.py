"""Where the bundled SYNTHETIC logs are: inside the installed package (``iptm/samples`` in a wheel, built
from the repository's ``logs/``), or the repository's ``logs/`` when running from a source checkout."""
from __future__ import annotations

from importlib import resources
from pathlib import Path

from calib import IptmError


def bundled_logs_dir() -> Path:
    """The folder of the bundled logs; IptmError saying how to regenerate them if neither place has them."""
    shipped = resources.files("iptm") / "samples"
    if shipped.is_dir():
        return Path(str(shipped))
    source = Path(__file__).resolve().parents[1] / "logs"
    if source.is_dir():
        return source
    raise IptmError(f"the bundled logs are missing (looked in {shipped} and {source}); reinstall the package "
                    "or regenerate them with `iptm synth --out logs`")
