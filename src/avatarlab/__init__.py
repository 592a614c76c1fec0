"""avatarlab: parametrized human head avatars from one monocular video (reproduction platform)."""

__version__ = "0.1.0"
