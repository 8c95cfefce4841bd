"""Evaluation: pose errors, matching, HOPE-paper tables and curves, BOP19 average recall.

Modules, one job each: ``metrics`` (the error functions), ``datasets`` (GT frames of a DOPE /
HOPE / BOP folder), ``models`` (object models: mesh points, diameter, symmetries), ``matching``
(per-pair errors and the greedy one-to-one match, shared by ``dope-hope evaluate`` and
``dope-hope demo``), ``reports`` (tables, CSV, curves), ``bop19`` (BOP19 AR), ``evaluate``
(the orchestrator behind ``dope-hope evaluate``).
"""
