from megalut_cli.cli import main

main()
