"""What the studies share: the real-data survey and its split (:mod:`experiments.common.autzen`) and the one
study runner (:mod:`experiments.common.study`: arms as data, validation chooses, the test block reports)."""
