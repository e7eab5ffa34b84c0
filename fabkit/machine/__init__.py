"""The machine that runs a program: its profile (:mod:`.profile`), the run time its
controller really takes (:mod:`.planner`) and the checks before cutting (:mod:`.limits`)."""
