"""The elimfast command-line interface (installed as the package ``elimfast_cli``)."""
