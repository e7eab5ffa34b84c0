"""``fabkit machine import FILE [-o OUT] [--json]``: a grbl ``$$`` dump or a LinuxCNC
INI -> a machine profile (YAML, the keys of the spec's ``machine`` section), for
``--machine OUT`` or to paste into a spec. Without ``-o`` the profile is printed.
Exit 2 on a file that is neither (one line naming it; nothing written).

``fabkit machine list [--json]``: the profiles shipped with fabkit, given by name
(``--machine grbl``)."""

from __future__ import annotations

import sys

from ._common import emit


def run(args) -> int:
    from ..errors import SpecError
    from ..io import check_outputs, write_atomic
    from ..machine.profile import import_settings, resolve_machine, safe_name, shipped_profiles, to_yaml

    if args.action == "list":
        rows = []
        for name in shipped_profiles():
            m = resolve_machine(name)
            rows.append((name, m))
        emit([f"{name}: {m.describe()}" for name, m in rows] +
             ["(use one by name: fabkit gcode SPEC --machine NAME; fabkit time PROGRAM --machine NAME)"],
             {"profiles": [{"name": n, "machine": m.to_dict()} for n, m in rows]}, args.json)
        return 0
    if not args.file:
        raise SpecError("machine import needs the settings FILE (a grbl $$ dump or a LinuxCNC INI)")
    if args.output:
        check_outputs({"--output": args.output}, inputs=[args.file])
    machine = import_settings(args.file)
    text = to_yaml(machine, comment=f"fabkit machine profile, imported from {safe_name(args.file)}")
    if args.output:
        write_atomic(args.output, text)
        emit([f"machine: {safe_name(args.output)}: {machine.describe()}"],
             {"output": args.output, "machine": machine.to_dict()}, args.json)
    elif args.json:
        emit([], {"output": None, "machine": machine.to_dict()}, True)
    else:
        sys.stdout.write(text)
    return 0
