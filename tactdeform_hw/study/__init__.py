"""Study runs: the TactDeform studies' trials driven through the whole pipeline, checked and reported.

``tactdeform-hw study task1|task2|task3|phase2 --out DIR`` runs a study's trial list
(:mod:`.scenarios`) through tracking, the renderer, the driver and the port — the emulator by default —
(:mod:`.runner`), checks what each trial delivered (:mod:`.checks`) and writes a JSON report, a short
Markdown summary and pictures of the array (:mod:`.report`), so a lab can check a setup before
participants arrive.
"""

from .scenarios import STUDIES, Segment, Study, Trial, build_study, select_trials

__all__ = ["STUDIES", "Segment", "Study", "Trial", "build_study", "select_trials"]
