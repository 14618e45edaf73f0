"""Diagnose: where simulated and measured frames disagree, which detector effect is missing, how strong.

The data flow:

- :mod:`perscli.diagnose.data` reads the measured frames (any order, put in
  time order), pairs them with the frames ``perscli render`` made of the same
  exposures, and gathers what the forward model needs: IDEAL, the fluence
  history, the exposure times;
- :mod:`perscli.diagnose.likelihood` turns a detector model (the registry of
  :mod:`perscli.detector.effects`, the same forward models render samples
  from) into the expectation and variance of every measured pixel, and the
  Gaussian likelihood of the data;
- :mod:`perscli.diagnose.candidates` lists the effects diagnose can add or
  re-tune (each a parameter of a registered effect), and
  :mod:`perscli.diagnose.search` fits them by likelihood
  (:mod:`perscli.diagnose.candidate_fit`, one candidate at a time;
  :mod:`perscli.diagnose.noise`, the noise pixels share), ranks them by
  delta chi^2 and delta BIC and adds the significant ones one by one;
- :mod:`perscli.diagnose.probes` bins the normalised residuals against the
  covariates that separate effects, and :mod:`perscli.diagnose.report`
  writes model.yaml, report.json, report.md and the figures.
"""
