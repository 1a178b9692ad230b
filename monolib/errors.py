"""The error of a study that cannot run, below every module that raises it (the study file, the zoo's manifests)."""


class StudyError(ValueError):
    """A study file that cannot be run; the message names the file and the key."""
