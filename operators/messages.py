"""The steps' messages as the sidebar says them: the procam command's options named by their fields.

The options a step declares with a sidebar label (addon/options.py) are named from that declaration; the rest
(the output folder, the Replace box, fields that gather several options) are listed here.

The steps are shared by the command and the sidebar, and their errors say what
to do in the command's words ("rerun with --force", "choose another --out").
In Blender those options are fields of the sidebar or of an operator's dialog,
so an operator reports a step's message through :func:`sidebar_text`, which
names each option by its field's label; an option the sidebar does not have
says that it belongs to the command.
"""

from __future__ import annotations

import re

from ..addon.options import sidebar_names
from ..addon.steps.calibrate import CalibrateOptions
from ..addon.steps.diagnose import DiagnoseOptions
from ..addon.steps.stage_c import StageCOptions

#: The command's options that are fields of the sidebar (scene properties), as a message names them: by the
#: field's label. An operator whose dialog has its own field for an option (a "Replace" box, its output folder)
#: passes that name instead.
SIDEBAR_NAMES = {
    **sidebar_names([CalibrateOptions, StageCOptions]),
    **{k: v for k, v in sidebar_names([DiagnoseOptions]).items() if k != "--scale"},
    "--force": "‘Replace Results’",
    "--out": "output folder",
    "--diagnosis": "‘Diagnosis’",
    "--targets": "‘Targets’",
}

#: An operator dialog's own "Replace" box (the sidebar's is ‘Replace Results’).
REPLACE_BOX = {"--force": "‘Replace’"}
#: The Diagnose panel's fields (``--scale`` means another scale to other commands: the lab's, the demo's).
DIAGNOSE_FIELDS = {"--out": "‘Diagnosis’ folder", **sidebar_names([DiagnoseOptions])}

_OPTION = re.compile(r"(?<![\w-])--[a-z][a-z-]*")
#: The Python API's keyword beside an option ("--force (force=True)"): the sidebar's field stands for both.
_KEYWORD = re.compile(r" \(\w+=True\)")


def sidebar_text(message: str, names: dict[str, str] | None = None) -> str:
    """``message`` with each of the command's options named as the sidebar names it (``names`` overrides
    :data:`SIDEBAR_NAMES` for one operator's own fields)."""
    table = {**SIDEBAR_NAMES, **(names or {})}

    def named(m: re.Match[str]) -> str:
        return table.get(m.group(0)) or f"{m.group(0)} (an option of the procam command)"

    return _OPTION.sub(named, _KEYWORD.sub("", message))
