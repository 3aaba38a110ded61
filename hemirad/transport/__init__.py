"""Light transport on a fixed mesh: the OpenGL context, hemicube rendering into item
atlases, delta form factors, what one hemicube saw (``HemicubeView``) and the progressive
shooting solver."""
