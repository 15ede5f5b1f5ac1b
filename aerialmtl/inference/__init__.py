"""Prediction: a model loaded once (:mod:`.predict`) run over windows of orthophotos into prediction folders."""
