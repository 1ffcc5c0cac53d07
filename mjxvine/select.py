"""`python -m mjxvine.select`: the old name of `python -m mjxvine.choose` (the best
checkpoint, chosen on validation worlds after training), kept so that it still answers."""

from mjxvine.choose import main as choose_main


def main(argv=None) -> int:
  return choose_main(argv, prog="python -m mjxvine.select")


if __name__ == "__main__":
  from mjxvine.atomic import command_main
  # SIGINT / SIGTERM: 130 / 143 in one line, selection.json kept
  command_main(main, keep_outputs=True)
