"""Studies: searching a space for a device (:mod:`.search`), reading a study back (:mod:`.results`), and
the typed records a study stores (:mod:`.records`)."""

from explorer.study.records import StudyRecord, TrialRecord, study_record, trial_record

__all__ = ["StudyRecord", "TrialRecord", "study_record", "trial_record"]
