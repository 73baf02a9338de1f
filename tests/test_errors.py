"""The package's errors keep their fields and message through pickling (studies' workers)."""

import pickle

from fluoronav.errors import InputError, RegistrationRefused


def test_registration_refused_pickles_with_its_fields() -> None:
    exc = RegistrationRefused("cm", "edge_ncc", "NCC 0.46 (at least 0.7)", view="AP")
    back = pickle.loads(pickle.dumps(exc))
    assert (back.stage, back.check, back.detail, back.view) == (
        "cm",
        "edge_ncc",
        "NCC 0.46 (at least 0.7)",
        "AP",
    )
    assert str(back) == str(exc) == "stage cm, view AP, check edge_ncc: NCC 0.46 (at least 0.7)"


def test_input_error_pickles_with_its_fields() -> None:
    exc = InputError("case/navigation.json", "field 'side' must be left or right")
    back = pickle.loads(pickle.dumps(exc))
    assert (back.source, back.problem, str(back)) == (exc.source, exc.problem, str(exc))
