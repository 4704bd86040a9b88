"""Helpers the test modules share (scenes, captures, problem catalogues, stores), so that no test module imports
another (#56; optimistix's tests/helpers.py is the model). Each module says what it builds and from what truth."""
