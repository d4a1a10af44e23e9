"""Validation studies: the thesis's figures and tables reproduced with the project's simulator.

They live in the repository, not in the installed package: run them from a clone with
``python pipelines/validate_<case>.py --out DIR`` (or ``plenopiv validate <case>`` where the
clone's ``pipelines/`` folder can be found). Each study computes in one module and, where it
draws figures, renders in a ``*_report`` module that imports it (never the other way round):

- :mod:`~pipelines.studies.calibration`: synthetic calibration (Figs 3.8, 3.9, 5.5);
- :mod:`~pipelines.studies.depth`, :mod:`~pipelines.studies.depth_report`: the depth study
  (Tables 5.1, 5.2, Figs 5.2-5.4);
- :mod:`~pipelines.studies.field_quality`, :mod:`~pipelines.studies.field_quality_report`:
  reconstruction quality of particle fields;
- :mod:`~pipelines.studies.letters_data`, :mod:`~pipelines.studies.letters`,
  :mod:`~pipelines.studies.letters_report`: the light field of the real plenoptomos image;
- :mod:`~pipelines.studies.realcam`, :mod:`~pipelines.studies.realcam_report`: the chain on
  renders through a modelled real camera, as recorded and preprocessed;
- :mod:`~pipelines.studies.tracking`, :mod:`~pipelines.studies.tracking_report`: particle
  tracking against correlation;
- :mod:`~pipelines.studies.uncertainty`: coverage of the per-vector uncertainty;
- :mod:`~pipelines.studies.vortex`: whole-chain accuracy on vortex flows;
- :mod:`~pipelines.studies.output`: how every study writes its figures, JSON and Markdown.
"""
