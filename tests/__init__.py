# A regular package, not a namespace one: a dependency that ships a top-level `tests` package
# (eds-utils does) would otherwise shadow this one, and `tests.support` would not import.
