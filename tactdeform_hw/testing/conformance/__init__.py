"""The conformance checks of an eTactileKit controller (or its emulator), runnable from any project: a test
module that star-imports :mod:`.checks_v1_2` or :mod:`.checks_v2` gets the checks, their fixtures and the
hook that picks the targets (:mod:`.targets`: every emulated target, or the one ``--etactile-device``
names).  See ``docs/testing-downstream.md`` and ``docs/firmware-guide-conformance.md``."""
