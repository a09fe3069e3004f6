"""Where the benchmark's real data lives, for an installed package as much as for a checkout.

Never derived from this file's place in the repository, which points into site-packages once
installed. Order: the explicit ``--data``, then ``$MSFNET_DATA``, then
``./shared/data`` and ``../shared/data`` relative to the current directory.
"""

from __future__ import annotations

import os
from pathlib import Path

from msfnet.common.errors import InputError
from msfnet.common.vocabulary import declare, opt, verbatim

# msf-bench --data: the folder holding the benchmark's real stacks
declare("data", "--data")
ENV_VAR = "MSFNET_DATA"
RELATIVE_CANDIDATES = (Path("shared") / "data", Path("..") / "shared" / "data")


def data_root(
    explicit: str | Path | None = None,
    *,
    cwd: Path | None = None,
    env: dict[str, str] | None = None,
) -> Path:
    """The data root folder (holding DiLiGenT/, psmImages/); InputError naming what was tried.

    An explicit path or $MSFNET_DATA must exist: a typo there is an error, not a silent
    fallback to another folder.
    """
    env = dict(os.environ) if env is None else env
    cwd = Path.cwd() if cwd is None else cwd
    if explicit is not None:
        path = Path(explicit).expanduser()
        if not path.is_dir():
            raise InputError(f"{opt('data')}: folder not found", path, option="data")
        return path
    if env.get(ENV_VAR):
        path = Path(env[ENV_VAR]).expanduser()
        if not path.is_dir():
            raise InputError(f"${ENV_VAR}: folder not found", path)
        return path
    tried = [cwd / rel for rel in RELATIVE_CANDIDATES]
    for path in tried:
        if path.is_dir():
            return path.resolve()
    raise InputError(
        f"no data folder: pass {opt('data', verbatim('DIR'))} (holding DiLiGenT/ballPNG) or set "
        f"${ENV_VAR}; also looked in {', '.join(str(p) for p in tried)}"
    )


__all__ = ["ENV_VAR", "data_root"]
