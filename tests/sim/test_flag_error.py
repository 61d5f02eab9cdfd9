"""sim.errors.flag_error: a job model's validation failure as one error naming the flags."""

from pydantic import ValidationError, field_validator

from sim.configio import StrictModel
from sim.errors import AdvobjError, flag_error


class _Err(AdvobjError, ValueError):
    pass


class _Own(AdvobjError, ValueError):
    pass


class _Job(StrictModel):
    out_dir: str
    count: int = 1
    name: str = "x"

    @field_validator("name")
    @classmethod
    def _own(cls, v):
        if v == "own":
            raise _Own("name: the validator's own one-line error")
        return v


def _error(extra=None, **fields):
    try:
        _Job(**fields)
    except ValidationError as err:
        return flag_error(err, lambda f: "--" + f.replace("_", "-"), "job", _Err, extra=extra)
    raise AssertionError("no validation error")


def test_each_problem_names_its_flag_in_one_line_of_the_given_class():
    e = _error(count="many")
    assert isinstance(e, _Err) and "\n" not in str(e)
    assert str(e).startswith("--out-dir: ") and "; --count: " in str(e)


def test_a_validators_own_project_error_is_returned_as_it_is():
    e = _error(out_dir="o", name="own")
    assert type(e) is _Own and str(e) == "name: the validator's own one-line error"


def test_unknown_fields_read_the_extra_text_and_more_than_three_problems_are_counted():
    e = _error(extra="not an option", out_dir="o", a=1, b=2, c=3, d=4)
    assert str(e).startswith("a: not an option; b: not an option; c: not an option")
    assert str(e).endswith("(and 1 more)")
