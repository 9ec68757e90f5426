"""``elimfast``: click commands that parse, call the library and print; no numerics here."""
import click

import elimfast


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(elimfast.__version__, prog_name="elimfast")
def cli():
    """Invariant-conserving integrators for Hamiltonian problems.

    Example: elimfast --version
    """


if __name__ == "__main__":
    cli()
