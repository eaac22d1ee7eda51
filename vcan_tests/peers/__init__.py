"""peers - independent bus peers for chcos' tests (C sources built by the tests)."""
