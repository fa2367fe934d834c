"""The machinery behind ``tools/vcan_run.py``: find a kernel with SocketCAN vcan and run
the ``vcan``-marked tests in it.

Ways, tried in this order by ``--way auto``:

- ``native``: the host kernel has CAN (``socket(AF_CAN)`` works and vcan0 can be up);
- ``uml-system``: the system's user-mode Linux, ``/usr/bin/linux.uml`` (package
  ``user-mode-linux``), if a probe boot of a few seconds succeeds (bookworm's and
  trixie's panic at init on CPUs with AMX);
- ``uml-testing``: user-mode Linux from Debian testing, fetched through a private apt
  list, unpacked with its own libc and patchelf'ed, cached, probed the same way;
- ``qemu``: bookworm's own kernel under QEMU (TCG, much slower).

See /work/shared/notes/vcan-on-amx-hosts.md and vcan-without-kernel-support.md.
"""
