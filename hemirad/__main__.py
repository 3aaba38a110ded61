from hemirad.cli import main

raise SystemExit(main())
