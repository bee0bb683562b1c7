"""``python -m kalmansfm`` runs the command line."""

if __name__ == "__main__":
    from .cli.main import run

    run()
