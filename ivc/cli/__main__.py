from ivc.cli import main

main()
