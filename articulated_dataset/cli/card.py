"""``artdata card``: a Hugging Face dataset card and Croissant metadata for splits to publish."""

from __future__ import annotations

import click


@click.command("card")
@click.argument("path", type=click.Path())
@click.option("--out", type=click.Path(file_okay=False), default=None,
              help="Folder to write README.md and croissant.json into (default: PATH). Their data paths are relative "
                   "to it: to upload, write them into the folder you upload.")
@click.option("--overwrite", is_flag=True, help="Replace an existing README.md and croissant.json.")
@click.option("--datasheet", type=click.Path(dir_okay=False), default=None,
              help="Datasheet (Markdown with a YAML header) to publish instead of the repository's DATASHEET.md; "
                   "needed for ingested real captures (docs/publishing.md lists its sections).")
@click.option("--citation", type=click.Path(dir_okay=False), default=None,
              help="CITATION.cff to cite instead of the repository's.")
@click.option("--url", default=None, help="Where the dataset is published (e.g. https://huggingface.co/datasets/USER/NAME): "
                                          "the Croissant url.")
def card_cmd(path, out, overwrite, datasheet, citation, url):
    """Write a Hugging Face dataset card (README.md) and Croissant metadata (croissant.json) for the splits at PATH
    (a split folder, a class folder or a data root <class>/<split>/): one datasets config per class, its splits'
    shards as data_files, the schema's fields with units, the datasheet, the citation. Needs the publish extra
    (datasets, mlcroissant). See docs/publishing.md."""
    from articulated_dataset.format.card import write_card

    for written in write_card(path, out, overwrite=overwrite, datasheet=datasheet, citation=citation, url=url):
        click.echo(f"wrote {written}")


COMMANDS = [card_cmd]
