"""Small pieces every other subpackage shares (parameter specs, joint-list text); imports nothing
of the package."""
