from radfield.cli.main import main

main()
