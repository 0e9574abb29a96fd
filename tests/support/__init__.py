"""Support code for the tests: helpers and fixtures shared by test modules."""
