"""motok.gpt"""
