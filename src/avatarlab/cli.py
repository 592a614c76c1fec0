"""`avatarlab <command> [hydra overrides]`: a thin front door to the Hydra entry points."""
from __future__ import annotations

import runpy
import sys

COMMANDS = {
    "render-demo": ("avatarlab.evaluate.head_model_demo", "PNG grid sweeping every head-model parameter"),
    "dlib-check": ("avatarlab.evaluate.dlib_check", "dlib detection rate and NME on renders of the head model"),
}


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in {"-h", "--help"} or argv[0] not in COMMANDS:
        print("usage: avatarlab <command> [hydra overrides ...]\n\ncommands:")
        for name, (_, what) in COMMANDS.items():
            print(f"  {name:<14} {what}")
        return 0 if argv and argv[0] in {"-h", "--help"} else 2
    module = COMMANDS[argv[0]][0]
    sys.argv = [module, *argv[1:]]
    runpy.run_module(module, run_name="__main__")
    return 0


if __name__ == "__main__":
    sys.exit(main())
