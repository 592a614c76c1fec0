"""The errors a user can cause, each reported as one line that names the culprit (file, key or subject)."""


class InputFileError(ValueError):
    """A file that is missing, unreadable or not what the step expects; the message names the file."""


class ConfigError(ValueError):
    """A setting that cannot work (wrong type, out of range, inconsistent with the data); names the key."""


class InputError(ValueError):
    """Input data a step cannot use (too few frames, no face, ...); names the subject and the file."""


class TrainingError(ValueError):
    """Training that cannot go on (a loss that is not finite); names the step's output, the iteration and the last
    checkpoint kept."""


USER_ERRORS = (InputFileError, ConfigError, InputError, TrainingError)
