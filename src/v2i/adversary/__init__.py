"""The adversary: fuzzing the services' inputs, hostile messages and keyed attacks against a live site."""
