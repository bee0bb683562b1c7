"""Running the CLI in-process as a test does: the exit code whether ``main`` returns it or argparse exits."""

from kalmansfm.cli.main import main


def exit_code(argv: list[str]) -> int:
    """``kalmansfm argv``'s exit code (argparse's usage errors end in SystemExit, the rest return one)."""
    try:
        return main(argv)
    except SystemExit as exc:
        return exc.code
