"""Host-observable protocol behaviour of an eTactileKit controller (or its emulator), firmware v1.2: the
package's checks (:mod:`tactdeform_hw.testing.conformance.checks_v1_2`), run here on every emulated target
or on the one ``--device`` names."""

from tactdeform_hw.testing.conformance.checks_v1_2 import *  # noqa: F403 - the checks, their fixtures and hook
