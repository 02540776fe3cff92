"""How motok marks the files it writes that have room for a mark, so that it can tell them from
files it did not write and never replace those (:func:`motok.cli.output_files.foreign_file`).
Nothing heavy here: the writers and the command line's checks both import it."""

MARK = "written by motok"  # a PNG text chunk, a GIF comment, an MP4 comment
MD_MARK = "<!-- written by motok -->"  # a Markdown report's first line (invisible once rendered)
