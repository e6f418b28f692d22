"""Suite-wide pytest hooks."""

#: Test files that take minutes on the CPU, longest first (seconds on the 2-core development machine,
#: 2026-11-25, a clean clone: 1130, 1073, 772, 634, 299 and 237 of the suite's 4785; after the stress stopped
#: calling svd3, about 880, 600, 550, 380, 200 and 150 of 3400; test_doctor_e2e then gained a 400 s test).
#: They run first, so that under ``make test`` (pytest-xdist, 2 workers, ``--dist loadfile
#: --no-loadscope-reorder``: files handed out in this order) each worker starts on long files and the short
#: ones fill in the end. xdist's default order (files
#: with the most tests first) left these few-test files for last; replaying its rule on the measured times gives
#: one worker 47 minutes and the other 33 (benchmarks/RESULTS.md, session 19).
LONG_FIRST = (
    "identification/test_synth_recovery.py",
    "identification/test_doctor_e2e.py",  # about 700-900 s: a hidden fracture and stiffness field too (2026-11-25)
    "identification/test_doctor.py",
    "identification/test_synth_recovery_dough.py",
    "identification/test_single_camera.py",
    "identification/test_uncertainty.py",
)


def pytest_collection_modifyitems(config, items):
    def rank(item):
        path = item.path.as_posix()
        return next((i for i, f in enumerate(LONG_FIRST) if path.endswith("/tests/" + f)), len(LONG_FIRST))

    items.sort(key=rank)  # stable: every file's tests keep their order and stay together
