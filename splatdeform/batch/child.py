"""``python -m splatdeform.batch.child``: one scan in its own process (see ``run_isolated``).

Protocol: prints ``ready`` once imported, reads one pickled Job from stdin, writes the pickled
report row to stdout. Anything the scan prints goes to stderr, so stdout carries only the row.
"""

from __future__ import annotations

import os
import pickle
import sys


def main() -> int:
    from .worker import cap_memory, process_scan, warm_up, worker_init

    worker_init(os.getppid())   # SIGTERM unwinds (temp folders, partial outputs); exit
                                # when the Dask worker that started us is gone
    out = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)        # stray prints must not corrupt the row
    sys.stdout = sys.stderr
    warm_up()
    out.write(b"ready\n")
    out.flush()
    job = pickle.loads(sys.stdin.buffer.read())
    cap_memory(job.memory_budget)   # a process of its own: the cap cannot hurt the Dask worker
    row = process_scan(job)
    out.write(pickle.dumps(row))
    out.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())
