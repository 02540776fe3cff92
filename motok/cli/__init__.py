"""motok.cli: the command line. Importing it (before torch) makes OpenMP's idle threads sleep
instead of spinning, unless the user chose otherwise: on a machine whose cores are all busy, a
spinning torch thread holds a core that MuJoCo's workers or another process need, and one other
CPU-bound process then slowed a 2-core training 10x; with sleeping threads it costs 25 %
(docs/control/expert.md "Throughput")."""

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
