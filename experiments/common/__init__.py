"""What the studies share (README.md here): the real-data survey and its split (:mod:`experiments.common.autzen`),
the one study runner with the height bins and the scores of a spread (:mod:`experiments.common.study`), prediction
folders on the survey (:mod:`experiments.common.maps`) and their evaluation (:mod:`experiments.common.reports`). No
study imports another study's ``run.py``."""
