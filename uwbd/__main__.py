from uwbd.cli import main

raise SystemExit(main())
