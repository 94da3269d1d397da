"""`cohflash scenes`: the built-in scenes and the effects a scene can switch on."""

from __future__ import annotations


def add_parser(sub) -> None:
    p = sub.add_parser("scenes", help="list built-in scenes and effects")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..effects import KNOWN_EFFECTS
    from ..scenes import BUILTIN_SCENES

    print("built-in scenes (default effects):")
    for name, make in BUILTIN_SCENES.items():
        s = make()
        print(f"  {name:10s} {s.description}\n  {'':10s} effects: {', '.join(s.effects)}")
    print("  file       --depth-map FILE [--reflectance-map FILE] (.npy or image)\n\neffects:")
    for name, text in KNOWN_EFFECTS.items():
        print(f"  {name:17s} {text}")
    return 0
