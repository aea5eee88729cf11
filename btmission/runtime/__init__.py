"""Running missions: agents, the coordinator, the message bus, events, the report.

``btmission.runtime.runner.MissionRun`` runs a mission in the embedded simulator
(:mod:`btmission.backends.sim`); ``btmission run`` and ``btmission report`` are its CLI. Import
the modules you need (they load numpy, py_trees and, for NMPC, CasADi), e.g.::

    from btmission.runtime.runner import MissionRun
    from btmission.runtime.events import JsonlEventLog, Recorder
    from btmission.runtime.report import report_from_log, format_report
"""
