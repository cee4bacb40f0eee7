import csv

from streaklab.bench.tables import write_csv


def test_columns_are_every_key_in_order_of_first_use_and_floats_have_six_digits(tmp_path):
    path = tmp_path / "t.csv"
    write_csv(path, [{"a": 1.0 / 3.0, "b": "x"}, {"c": 7, "a": 2.0}])
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    assert rows == [["a", "b", "c"], ["0.333333", "x", ""], ["2", "", "7"]]


def test_given_fields_choose_and_order_the_columns(tmp_path):
    path = tmp_path / "t.csv"
    write_csv(path, [{"a": 1, "b": 2, "extra": 3}], fields=("b", "a"))
    with open(path, newline="") as fh:
        assert list(csv.reader(fh)) == [["b", "a"], ["2", "1"]]
