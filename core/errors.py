"""The root of neumip's user-facing errors.

Every error that reports a user's mistake or an unusable input (bad queries, a corrupt model or
checkpoint, an incomplete data set, an unreachable server, a missing LLVM) derives from
:class:`NeumipError`, so the CLI turns each into one line and exit status 2 instead of a traceback.
"""


class NeumipError(Exception):
    """An error whose message alone tells the user what went wrong and what to do."""


class CommandError(NeumipError):
    """An error a command reports to the user as one line, exit status 2."""


def differences(old: dict, new: dict, labels: tuple[str, str] = ("checkpoint", "now"), *, ignore=()) -> list[str]:
    """'key: OLD_LABEL x, NEW_LABEL y' for every setting that differs between two settings dicts (nested dicts'
    keys joined by dots, a key one side lacks "unset"), for the message that refuses to mix them."""
    out = []
    for key in sorted((old.keys() | new.keys()) - set(ignore)):
        a, b = old.get(key), new.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            out += [f"{key}.{line}" for line in differences(a, b, labels)]
        elif a != b:
            shown = (repr(d[key]) if key in d else "unset" for d in (old, new))
            out.append(f"{key}: " + ", ".join(f"{label} {value}" for label, value in zip(labels, shown)))
    return out
