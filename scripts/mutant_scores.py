"""Mutation scores per module from mutmut's results (`make mutants` prints them last).

    .venv/bin/mutmut results --all true | python scripts/mutant_scores.py

Reads lines ``NAME: STATUS`` and prints, per module, killed / viable and the survivors. Viable
mutants are those that ran (``not checked`` ones, generated but outside the run's names, are left
out); a timeout counts as killed (the change made the tests hang), ``no tests`` as survived.
"""
import re
import sys
from collections import defaultdict

KILLED = {"killed", "timeout", "segfault"}
SKIPPED = {"not checked", "skipped"}


def module_of(name: str) -> str:
    # motok.quantize.vq.xǁVectorQuantizerǁforward__mutmut_1 -> motok.quantize.vq
    return re.split(r"\.x(?:ǁ|_)", name, maxsplit=1)[0]


def main() -> None:
    counts: dict[str, list[int]] = defaultdict(lambda: [0, 0])
    survivors: dict[str, list[str]] = defaultdict(list)
    for line in sys.stdin:
        name, sep, status = line.strip().rpartition(": ")
        if not sep or status in SKIPPED:
            continue
        module = module_of(name)
        counts[module][1] += 1
        if status in KILLED:
            counts[module][0] += 1
        else:
            survivors[module].append(f"{name} ({status})")
    total = [sum(c[0] for c in counts.values()), sum(c[1] for c in counts.values())]
    for module, (killed, viable) in sorted(counts.items()) + [("all", tuple(total))]:
        print(f"{module:36s} {killed:5d} / {viable:<5d} {100 * killed / max(viable, 1):5.1f} %")
    for module in sorted(survivors):
        print(f"\n{module}: {len(survivors[module])} survived")
        for s in survivors[module]:
            print("   ", s)


if __name__ == "__main__":
    main()
