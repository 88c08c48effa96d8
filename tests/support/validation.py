"""USD's own validation for the tests: every registered validator run over an authored stage."""

from __future__ import annotations

from pxr import Usd, UsdValidation

from allo_usd.usd import schema


def validation_errors(path, warnings: bool = False) -> list[str]:
    """Errors (and, with `warnings`, warnings too) that all registered validators find on `path`."""
    schema.register()
    validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
    assert len(validators) > 10
    errors = UsdValidation.ValidationContext(validators).Validate(Usd.Stage.Open(str(path)))
    return [f"{e.GetName()}: {e.GetMessage()}" for e in errors
            if e.GetType() == UsdValidation.ValidationErrorType.Error
            or (warnings and e.GetType() == UsdValidation.ValidationErrorType.Warn)]
