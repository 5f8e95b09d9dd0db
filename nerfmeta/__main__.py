from nerfmeta.cli import main

raise SystemExit(main())
