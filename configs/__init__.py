"""The packaged experiment configs (`detmatch train --config tiny`): this directory is
installed as the package `detmatch.configs`."""
