"""The package's error for failures outside its control that the user can act on."""


class CommandError(RuntimeError):
    """A failure outside the package's control (a hub refusing, say) that the user can act on."""
