"""Exception types.

Every error a user can cause (bad scene, bad file, bad option) is a ``ClvolError``;
the CLI turns it into a one-line message and exit status 2. Anything else is a bug.
"""


class ClvolError(Exception):
    """A problem with the user's input: a scene, a file, an option."""


class SceneError(ClvolError):
    """A scene file is malformed; the message starts with the file and the dotted field."""


class VolumeError(ClvolError):
    """A volume file or grid is malformed or holds values we refuse (NaN, Inf, < 0)."""


class ImageError(ClvolError):
    """An image file cannot be read or written."""


class DeviceError(ClvolError):
    """No OpenCL device matches the request, or none is installed."""


class BuildError(ClvolError):
    """An OpenCL program failed to compile; the message carries the file and compiler log.
    ``stem`` (the kernel file's stem), ``device`` and ``first_error`` (the log's first error
    line) give the one-line form, ``one_line()``."""

    def __init__(self, message: str, stem: str | None = None, device: str | None = None,
                 first_error: str | None = None):
        super().__init__(message)
        self.stem, self.device, self.first_error = stem, device, first_error

    def one_line(self) -> str:
        if self.stem is None:
            return str(self).splitlines()[0] if str(self) else "build failed"
        return f"{self.stem}.cl failed to build on {self.device}: {self.first_error}"


class WeightsError(ClvolError):
    """A weight file is missing, malformed, of another version or of another feature contract."""


class NetworkInputError(ClvolError):
    """Inputs to the network (features, config, albedo) that do not match its layout."""
