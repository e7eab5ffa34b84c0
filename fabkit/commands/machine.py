"""``fabkit machine import FILE [-o OUT] [--json]``: a grbl ``$$`` dump or a LinuxCNC
INI -> a machine profile (YAML, the keys of the spec's ``machine`` section), for
``--machine OUT`` or to paste into a spec. Without ``-o`` the profile is printed.
Exit 2 on a file that is neither (one line naming it; nothing written)."""

from __future__ import annotations

import sys

from ._common import emit


def run(args) -> int:
    from ..io import check_outputs, write_atomic
    from ..machine.profile import import_settings, to_yaml

    if args.output:
        check_outputs({"--output": args.output}, inputs=[args.file])
    machine = import_settings(args.file)
    text = to_yaml(machine, comment=f"fabkit machine profile, imported from {args.file}")
    if args.output:
        write_atomic(args.output, text)
        emit([f"machine: {args.output}: {machine.describe()}"],
             {"output": args.output, "machine": machine.to_dict()}, args.json)
    elif args.json:
        emit([], {"output": None, "machine": machine.to_dict()}, True)
    else:
        sys.stdout.write(text)
    return 0
