from viewloc_cli.main import main

raise SystemExit(main())
