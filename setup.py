"""The C extensions (the filter's core, uwbd/fusion/core/_core.c, and the daemon's serial reader,
uwbd/service/_reader.c) are built here; everything else is in pyproject.toml.

``optional=True``: where no C compiler is found the install goes on without it and uwbd
runs its pure-Python reference (``uwbd version`` says which one runs).
"""

from setuptools import Extension, setup

setup(ext_modules=[
    Extension(
        "uwbd.fusion.core._core", ["uwbd/fusion/core/_core.c", "uwbd/fusion/core/_state.c",
                              "uwbd/fusion/core/_update.c", "uwbd/fusion/core/mm_range.c",
                              "uwbd/fusion/core/_lsq.c", "uwbd/fusion/core/_rest.c",
                              "uwbd/fusion/core/_imu.c",
                              "uwbd/fusion/core/_checks.c"],
        depends=["uwbd/fusion/core/_core.h"],
        # a * b + c rounded as Python rounds it (no fused multiply-add): the same bits; -O3
        # vectorises the element-wise loops (sums are never reassociated: the same bits)
        extra_compile_args=["-O3", "-ffp-contract=off", "-fno-fast-math"],
        optional=True,
    ),
    # the per-message loops of reading a whole log (uwbd/logs/scan.py, mcaplog.py)
    Extension("uwbd.logs._scan", ["uwbd/logs/_scan.c"], depends=["uwbd/_tuple.h"],
              extra_compile_args=["-O2"], optional=True),
    # the output log's open chunk and its message indexes (uwbd/logs/chunked.py)
    Extension("uwbd.logs._chunk", ["uwbd/logs/_chunk.c"], extra_compile_args=["-O2"],
              optional=True),
    # the WitMotion parser and the common Nooploop read (drivers/wit.py, nlink.py, accel.py)
    Extension("drivers._frames", ["drivers/_frames.c", "drivers/_wit.c"],
              depends=["drivers/_wit.h"], extra_compile_args=["-O2"], optional=True),
    # the daemon's serial reads on a thread of their own (uwbd/service/ports.py)
    Extension("uwbd.service._reader", ["uwbd/service/_reader.c"], extra_compile_args=["-O2"],
              extra_link_args=["-pthread"], optional=True),
])
