"""One-off measurements behind design choices, kept so their figures can be reproduced
(`python -m bench.experiments.<name>`). Not part of `renderloop bench`: each answers one
question recorded in the doc it names, on the validation scenes unless it says otherwise."""
