"""``python -m splatdeform.basis.kernel_warm`` (``make setup``): build the OpenCL kernels a
deform uses on this machine's default device, so that the first ``deform`` finds them in the
driver's cache (:mod:`.kernel_cache`). Nothing, and exit 0, without a device."""

from __future__ import annotations

from splatdeform.basis import opencl
from splatdeform.basis.kernel_cache import set_note_sink


def warm(device: str | None = None) -> list[str]:
    """Build (or load from the cache) the kernels a deform uses: the one-shot K = 3 with and
    without gradients and the stored basis of one handle (K = 4; ``--reuse``). Returns what
    was built; nothing without a device."""
    if not opencl.opencl_available(device):
        return []
    done = []
    for k, gradients in ((3, True), (3, False), (4, True)):
        opencl.prepare_device(device, k, gradients)
        done.append(f"basis K={k}{'' if gradients else ' (no gradients)'}")
    return done


if __name__ == "__main__":
    import sys

    set_note_sink(lambda line: print(f"splatdeform: {line}", file=sys.stderr, flush=True))
    built = warm()
    print("OpenCL kernels ready: " + ", ".join(built) if built else
          "no OpenCL device: nothing to build (deform uses the numpy backend)")
